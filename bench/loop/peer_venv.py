"""The peer's own virtual environment: ``bench/.rpio-venv`` with ``robosapiensio==0.4.3``.

RPIO 0.4.3 pins old versions of numpy, redis, paho-mqtt and some fifty more packages, so it
never shares the workspace environment. ``ensure_venv()`` creates it once (stdlib ``venv`` +
pip, so pip's own configuration and mirrors apply) and skips the work when the environment
is present and ``rpio.clientLibraries.rpclpy`` imports at the pinned version.

``python -m bench.loop.peer_venv`` does the same from the command line.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
VENV = ROOT / "bench" / ".rpio-venv"
PACKAGE = "robosapiensio"
VERSION = "0.4.3"
INDEX_PROBE = f"https://pypi.org/simple/{PACKAGE}/"
INSTALL_TIMEOUT_S = 900.0

_CHECK = (
    "import importlib.metadata as m, sys\n"
    "import rpio.clientLibraries.rpclpy.node\n"
    f"sys.exit(0 if m.version({PACKAGE!r}) == {VERSION!r} else 3)\n"
)


class PeerVenvError(RuntimeError):
    """The peer environment could not be created or is unusable."""


def venv_python(venv: Path = VENV) -> Path:
    return venv / "bin" / "python"


def _say(msg: str) -> None:
    print(f"  [rpio-venv] {msg}", file=sys.stderr, flush=True)


def is_ready(venv: Path = VENV) -> bool:
    """True when the venv exists and imports rpclpy from robosapiensio at the pinned version."""
    py = venv_python(venv)
    if not py.exists():
        return False
    try:
        done = subprocess.run([str(py), "-c", _CHECK], capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _pypi_reachable(timeout: float = 10.0) -> str | None:
    """None when the PyPI simple index answers, else why not."""
    try:
        with urllib.request.urlopen(INDEX_PROBE, timeout=timeout) as resp:
            resp.read(1)
    except (urllib.error.URLError, OSError) as exc:
        return str(getattr(exc, "reason", exc))
    return None


def ensure_venv(venv: Path = VENV, *, quiet: bool = False) -> Path:
    """Create ``venv`` with robosapiensio==0.4.3 unless it is already usable; return its python.

    Raises PeerVenvError with the reason (PyPI unreachable, pip failure, missing venv module).
    """
    if is_ready(venv):
        if not quiet:
            _say(f"{venv.relative_to(ROOT)} ready ({PACKAGE} {VERSION})")
        return venv_python(venv)
    py = venv_python(venv)
    if not py.exists():
        if venv.exists():  # a half-made directory from an interrupted run
            shutil.rmtree(venv)
        _say(f"creating {venv} with {sys.executable}")
        made = subprocess.run(
            [sys.executable, "-m", "venv", str(venv)], capture_output=True, text=True
        )
        if made.returncode != 0:
            raise PeerVenvError(
                f"python -m venv {venv} failed (is the venv/ensurepip module installed?):\n"
                + (made.stdout + made.stderr)[-2000:]
            )
    _say(f"installing {PACKAGE}=={VERSION} and its pinned dependencies (one-time, ~1-3 min)")
    cmd = [str(py), "-m", "pip", "install", "--disable-pip-version-check"]
    cmd += ["--progress-bar", "off", f"{PACKAGE}=={VERSION}"]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    except subprocess.TimeoutExpired as exc:
        why = _pypi_reachable()
        hint = f"PyPI unreachable ({why})" if why else "PyPI answers, but the install hung"
        raise PeerVenvError(f"pip install timed out after {exc.timeout:.0f} s: {hint}") from exc
    if done.returncode != 0:
        why = _pypi_reachable()
        tail = (done.stdout + done.stderr)[-3000:]
        if why is not None:
            raise PeerVenvError(
                f"cannot install {PACKAGE}=={VERSION}: PyPI ({INDEX_PROBE}) is unreachable: "
                f"{why}. The peer benchmark needs network access once to build {venv}.\n{tail}"
            )
        raise PeerVenvError(f"pip install {PACKAGE}=={VERSION} failed:\n{tail}")
    if not is_ready(venv):
        raise PeerVenvError(f"{venv}: installed, but rpio.clientLibraries.rpclpy does not import")
    _say(f"{venv.relative_to(ROOT)} ready ({PACKAGE} {VERSION})")
    return py


def main() -> int:
    try:
        print(ensure_venv())
    except PeerVenvError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
