"""The project's one error type (DESIGN §8).

Every check of user input raises :class:`MuscleMSSError` with a sentence that names what is
wrong and where (file, block, row, fibre) and the rule it breaks, so that a user can act on it.
"""


class MuscleMSSError(ValueError):
    """Bad input or an impossible request, described for the user.

    The message names the file / block / row and the broken rule, e.g.
    ``"fibres.vtm block 'gracilis': fibre 12 has 1 point; a fibre needs at least 2"``.
    """
