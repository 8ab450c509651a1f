"""Running Debian's ParaView (pvpython, pvbatch, paraview under xvfb) from the tests.

The child processes get ``plugin/shim`` on PYTHONPATH (the 5.11 ``getargspec`` fix, and this
checkout importable as ``muscle_mss``), the plugin folder on PV_PLUGIN_PATH, and a Numba cache of
their own (ParaView's numba 0.56 and the venv's numba must not share one).
"""
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
    env["NUMBA_CACHE_DIR"] = str(REPO / ".numba-cache" / "debian")
    env["PYTHONUNBUFFERED"] = "1"
    env.update({k: str(v) for k, v in extra.items()})
    return env


def run(command, timeout=600, cwd=REPO, **extra_env) -> subprocess.CompletedProcess:
    """Run a ParaView command line; fail with its output when it exits non-zero."""
    proc = subprocess.run([str(c) for c in command], cwd=cwd, env=paraview_env(**extra_env),
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
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
