"""Choose MuJoCo's offscreen OpenGL backend (``MUJOCO_GL``) before MuJoCo is imported.

MuJoCo binds its GL backend when ``import mujoco`` runs (``mujoco.rendering.classic.gl_context`` reads
``MUJOCO_GL`` once), so the choice must happen first. :func:`import_mujoco` is the one entry point the sim stage
uses: it respects a value the user already set, otherwise probes ``egl`` then ``osmesa`` (each in a short child
process, so a backend that crashes or hangs cannot poison this process), sets ``MUJOCO_GL`` to the first one that
creates a context, and imports MuJoCo. If none works it raises one :class:`~umi_aug.errors.SimError` that names
what was tried, why each failed and which apt packages fix it.

Nothing runs at import time of this module.
"""

from __future__ import annotations

import ctypes.util
import logging
import os
import subprocess
import sys
from types import ModuleType

from umi_aug.errors import SimError

__all__ = ["CANDIDATE_BACKENDS", "choose_backend", "select_gl_backend", "import_mujoco", "create_gl_context", "gl_backend"]

log = logging.getLogger(__name__)

#: Offscreen backends tried, in order, when ``MUJOCO_GL`` is unset (Linux, headless CPU machines).
CANDIDATE_BACKENDS: tuple[str, ...] = ("egl", "osmesa")
#: Seconds allowed for one child-process probe (import mujoco + create a 16×16 context).
PROBE_TIMEOUT_S: float = 60.0
#: Shared libraries each backend needs, and the Debian/Ubuntu packages that provide them.
_BACKEND_LIBS: dict[str, tuple[str, str]] = {
    "egl": ("EGL", "libegl1 libgl1-mesa-dri (Mesa software EGL: llvmpipe)"),
    "osmesa": ("OSMesa", "libosmesa6"),
}
_FIX = (
    "Install an offscreen OpenGL backend, e.g. `sudo apt-get install -y libegl1 libgl1-mesa-dri` (EGL, preferred) "
    "or `sudo apt-get install -y libosmesa6` (OSMesa), or set MUJOCO_GL to a backend that works on this machine "
    "(egl | osmesa | glfw with a display)."
)
_PROBE_CODE = (
    "import mujoco\n"
    "ctx = mujoco.GLContext(16, 16)\n"
    "ctx.make_current()\n"
    "ctx.free()\n"
    "print('ok')\n"
)

_chosen: str | None = None


def _probe(backend: str) -> tuple[bool, str]:
    """Try ``backend`` in a child process. Returns ``(works, reason_if_not)``."""
    lib, pkgs = _BACKEND_LIBS.get(backend, ("", ""))
    if lib and ctypes.util.find_library(lib) is None:
        return False, f"lib{lib} not found (apt package: {pkgs})"
    env = dict(os.environ, MUJOCO_GL=backend)
    env.pop("PYOPENGL_PLATFORM", None)  # MuJoCo sets it to match MUJOCO_GL
    try:
        res = subprocess.run(
            [sys.executable, "-c", _PROBE_CODE], env=env, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return False, f"probe timed out after {PROBE_TIMEOUT_S:.0f} s"
    if res.returncode == 0 and "ok" in res.stdout:
        return True, ""
    tail = (res.stderr.strip().splitlines() or ["(no output)"])[-1]
    return False, f"context creation failed: {tail[:300]}"


def choose_backend(user_value: str, mujoco_imported: bool, probe=_probe) -> str:
    """Pure decision behind :func:`select_gl_backend` (no caching, no environment writes).

    Args:
        user_value: the current ``MUJOCO_GL`` ("" if unset).
        mujoco_imported: MuJoCo is already imported (its backend is fixed).
        probe: ``backend -> (works, reason)``.

    Returns:
        The backend name.

    Raises:
        SimError: nothing to respect and no candidate works (names each attempt, its failure and the fix).
    """
    user = user_value.strip()
    if user or mujoco_imported:
        return user.lower() or "glfw"
    failures = []
    for backend in CANDIDATE_BACKENDS:
        ok, why = probe(backend)
        if ok:
            return backend
        failures.append(f"MUJOCO_GL={backend}: {why}")
        log.debug("MUJOCO_GL=%s unusable: %s", backend, why)
    raise SimError("no offscreen OpenGL backend works for MuJoCo. Tried " + "; ".join(failures) + ". " + _FIX)


def select_gl_backend() -> str:
    """Return the offscreen GL backend MuJoCo will use, choosing and exporting ``MUJOCO_GL`` if needed.

    Order: a backend already bound (MuJoCo imported) → the user's ``MUJOCO_GL`` → the first of
    :data:`CANDIDATE_BACKENDS` whose probe creates a context. The result is cached for the process.

    Raises:
        SimError: no candidate backend works (message lists each attempt and the apt packages to install).
    """
    global _chosen
    if _chosen is not None:
        return _chosen
    user = os.environ.get("MUJOCO_GL", "")
    backend = choose_backend(user, "mujoco" in sys.modules)
    if not user.strip() and "mujoco" not in sys.modules:
        os.environ["MUJOCO_GL"] = backend
        log.info("MuJoCo offscreen rendering: MUJOCO_GL=%s", backend)
    _chosen = backend
    return backend


def gl_backend() -> str:
    """The backend chosen by :func:`select_gl_backend` (chooses one if not yet done)."""
    return select_gl_backend()


def import_mujoco() -> ModuleType:
    """Select the GL backend (see :func:`select_gl_backend`) and return the imported ``mujoco`` module.

    Raises:
        SimError: MuJoCo is not installed (``pip install 'umi-aug[sim]'``) or no GL backend works.
    """
    select_gl_backend()
    try:
        import mujoco
    except ImportError as exc:
        raise SimError(
            f"MuJoCo is not installed ({exc}); install the sim extra: pip install 'umi-aug[sim]' "
            "(mujoco>=3.3,<3.10)"
        ) from exc
    return mujoco


def create_gl_context(width: int, height: int):
    """Create and make current an offscreen ``mujoco.GLContext`` of ``width × height`` pixels.

    Raises:
        SimError: the context cannot be created with the selected backend (names it and the fix).
    """
    mujoco = import_mujoco()
    backend = os.environ.get("MUJOCO_GL", "")
    if getattr(mujoco, "GLContext", None) is None:
        raise SimError(f"MuJoCo has no offscreen GL context for MUJOCO_GL={backend!r}. {_FIX}")
    try:
        ctx = mujoco.GLContext(int(width), int(height))
        ctx.make_current()
    except Exception as exc:  # noqa: BLE001 - backends raise many types (EGLError, RuntimeError, OSError)
        raise SimError(f"cannot create an offscreen OpenGL context with MUJOCO_GL={backend!r}: {exc}. {_FIX}") from exc
    return ctx
