"""The project's one error type (DESIGN §8).

Every check of user input raises :class:`MuscleMSSError` with a sentence that names what is
wrong and where (file, block, row, fibre) and the rule it breaks, so that a user can act on it.
"""


class MuscleMSSError(ValueError):
    """Bad input or an impossible request, described for the user.

    The message names the file / block / row and the broken rule, e.g.
    ``"fibres.vtm block 'gracilis': fibre 12 has 1 point; a fibre needs at least 2"``.
    """


def first_problem(problems) -> MuscleMSSError:
    """The error to raise for a non-empty list of problem sentences: the first one, saying how
    many more there are (``muscle-mss validate`` lists them all)."""
    more = f" (and {len(problems) - 1} more problems)" if len(problems) > 1 else ""
    return MuscleMSSError(problems[0] + more)
