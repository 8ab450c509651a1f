"""Running Debian's ParaView (pvpython, pvbatch, paraview under xvfb) from the tests.

The child processes get ``plugin/shim`` on PYTHONPATH (the 5.11 ``getargspec`` fix, and this
checkout importable as ``muscle_mss``) and the plugin folder on PV_PLUGIN_PATH. They load their
kernels from the user's kernel cache, as ParaView does outside the tests (the folder is keyed by
Python, Numba and NumPy: ParaView's numba 0.56 has its own beside the venv's), compiled there
once before the first of them runs (:func:`warm_paraview_python`), not inside a test's timeout.
"""
import atexit
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHIM = REPO / "plugin" / "shim"
PLUGIN_DIR = REPO / "plugin" / "paraview_plugins"
PLUGIN_FILE = PLUGIN_DIR / "muscle_mss_plugin.py"
SCRIPTS = Path(__file__).resolve().parent / "paraview_scripts"


def paraview_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "VIRTUAL_ENV")}
    venv_bin = str(Path(sys.executable).parent)
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                  if p != venv_bin)
    env["PYTHONPATH"] = str(SHIM)
    env["PV_PLUGIN_PATH"] = str(PLUGIN_DIR)
    env["PYTHONUNBUFFERED"] = "1"
    env.update({k: str(v) for k, v in extra.items()})
    return env


_WARM: list = []  # [True] once ParaView's Python's kernels were found or made compiled


def warm_paraview_python() -> None:
    """Compile ParaView's Python's kernels into the user's kernel cache, or find them compiled
    (a second or two: ./test.sh's ./setup.sh has compiled them), once per test process and with
    no timeout, so that no ParaView command's timeout is spent compiling."""
    if _WARM:
        return
    proc = subprocess.run(["pvpython", "-m", "muscle_mss.app.warm_up", "--quiet"], cwd=REPO,
                          env=paraview_env(), capture_output=True, text=True)
    if proc.returncode != 0:
        raise AssertionError(f"pvpython -m muscle_mss.app.warm_up exited {proc.returncode}\n"
                             f"{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    _WARM.append(True)


_X_SERVER: list = []  # the one Xvfb of this test process: [Popen, display]


def x_display() -> str:
    """The DISPLAY of one Xvfb (1280x1024x24) shared by every headless command of this test
    process, started on first use and stopped at exit.

    ``xvfb-run -a`` starts a server per command and guesses a free number from lock files; on
    CI a command once got a display whose server was not accepting connections ("bad X server
    connection. DISPLAY=:99") and pvpython aborted. ``Xvfb -displayfd`` picks a free number
    itself and writes it only once it accepts connections.
    """
    if _X_SERVER and _X_SERVER[0].poll() is None:
        return _X_SERVER[1]
    _X_SERVER.clear()
    read, write = os.pipe()
    server = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", "1280x1024x24",
                               "-nolisten", "tcp"], pass_fds=(write,),
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(write)
    with os.fdopen(read) as ready:
        number = ready.readline().strip()
    if not number:
        raise AssertionError(f"Xvfb did not start: {server.stderr.read().decode()[-2000:]}")
    atexit.register(server.terminate)
    _X_SERVER.extend([server, f":{number}"])
    return _X_SERVER[1]


def _headless(command: list, extra_env: dict) -> list:
    """``xvfb-run [-a] [-s ARGS] CMD…`` → ``CMD…`` on the shared server (see ``x_display``)."""
    if not command or command[0] != "xvfb-run":
        return command
    rest = command[1:]
    while rest and rest[0] in ("-a", "-s"):
        rest = rest[2:] if rest[0] == "-s" else rest[1:]
    extra_env["DISPLAY"] = x_display()
    return rest


BAD_X_CONNECTION = "bad X server connection"


def run(command, timeout=600, cwd=REPO, check=True, **extra_env) -> subprocess.CompletedProcess:
    """Run a ParaView command line; fail with its output when it exits non-zero (``check=False``:
    return it whatever its exit status, for a test of a failing command). A command
    written ``xvfb-run …`` runs on the test process's shared Xvfb (``x_display``); when
    ParaView aborts because that server refused the connection (seen once on CI with a server
    that had just served the previous command), the server is restarted and the command run
    once more: that is the test machine's fault, not the command's."""
    warm_paraview_python()
    headless = _headless([str(c) for c in command], extra_env)
    proc = subprocess.run(headless, cwd=cwd, env=paraview_env(**extra_env),
                          capture_output=True, text=True, timeout=timeout)
    if (proc.returncode != 0 and headless != [str(c) for c in command]
            and BAD_X_CONNECTION in proc.stderr):
        if _X_SERVER:
            _X_SERVER[0].terminate()
            _X_SERVER[0].wait()
        _X_SERVER.clear()
        headless = _headless([str(c) for c in command], extra_env)
        proc = subprocess.run(headless, cwd=cwd, env=paraview_env(**extra_env),
                              capture_output=True, text=True, timeout=timeout)
    command = headless
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, command))} exited {proc.returncode}\n"
                             f"--- stdout ---\n{proc.stdout[-6000:]}\n"
                             f"--- stderr ---\n{proc.stderr[-6000:]}")
    return proc


def run_script(*command, timeout=600, cwd=REPO, **extra_env) -> dict:
    """Run ``tests/paraview_scripts/<script>`` with a tool (``run_script("pvpython", "x.py",
    *args)``, or ``"xvfb-run", "-a", "pvpython", "x.py", …``); the script prints one line
    ``RESULT <json>``, which is returned."""
    script = next(c for c in command if str(c).endswith(".py"))
    command = [SCRIPTS / c if c == script else c for c in command]
    proc = run(command, timeout=timeout, cwd=cwd, **extra_env)
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise AssertionError(f"{script} printed no RESULT line\n{proc.stdout[-4000:]}\n"
                         f"{proc.stderr[-4000:]}")
