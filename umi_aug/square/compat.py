"""Import robosuite 1.4.1 / robomimic 0.3.0 on MuJoCo 3.x (the only place that knows their quirks).

robomimic 0.3.0's ``envs/env_robosuite.py`` does ``import mujoco_py`` at top level, only to name an exception
type (``mujoco_py.builder.MujocoException``); mujoco_py does not install with MuJoCo 3.x. robomimic fixed this
right after the 0.3.0 tag (robomimic#66, commit 8df6e8e), but PyPI has no later release.
:func:`install_mujoco_py_stub` registers a stand-in module for that one name. robosuite imports MuJoCo at
import time, so :func:`import_robosuite` selects the offscreen GL backend first (:func:`umi_aug.sim.gl.import_mujoco`).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import logging
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from umi_aug.errors import SimError
from umi_aug.sim.gl import import_mujoco

__all__ = ["install_mujoco_py_stub", "import_robosuite", "import_robomimic_env_utils", "robomimic_quiet"]

_INSTALL_HINT = ("install the robomimic extra: pip install -c constraints.txt -e '.[robomimic]' "
                 "(robosuite==1.4.1, robomimic==0.3.0 --no-deps, h5py)")


def install_mujoco_py_stub() -> None:
    """Register a stand-in ``mujoco_py`` (with ``builder.MujocoException = Exception``) unless a real one is
    importable or already loaded. Idempotent. Needed before importing robomimic 0.3.0's robosuite wrapper."""
    if "mujoco_py" in sys.modules:
        return
    mod = types.ModuleType("mujoco_py")
    builder = types.ModuleType("mujoco_py.builder")
    builder.MujocoException = Exception  # type: ignore[attr-defined]
    mod.builder = builder  # type: ignore[attr-defined]
    mod.__umi_aug_stub__ = True  # type: ignore[attr-defined]
    sys.modules["mujoco_py"] = mod
    sys.modules["mujoco_py.builder"] = builder


def _empty_private_macros() -> None:
    """robosuite warns three lines on import when it has no ``macros_private.py`` (its optional per-install
    settings file). Without one, register an empty module under that name (the defaults, as robosuite uses them
    then) so nothing is printed; a real file is left to be imported."""
    if "robosuite" in sys.modules or "robosuite.macros_private" in sys.modules:
        return
    spec = importlib.util.find_spec("robosuite")  # locates the package without importing it
    if spec is None or not spec.submodule_search_locations:
        return
    if any((Path(p) / "macros_private.py").exists() for p in spec.submodule_search_locations):
        return
    sys.modules["robosuite.macros_private"] = types.ModuleType("robosuite.macros_private")


@contextlib.contextmanager
def robomimic_quiet() -> Iterator[None]:
    """What robomimic / robosuite print to stdout inside (environment banners, observation-spec tables) goes to
    this module's debug log instead of the user's console."""
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            yield
    finally:
        text = buf.getvalue().strip()
        if text:
            logging.getLogger(__name__).debug("robomimic: %s", text)


def import_robosuite() -> ModuleType:
    """Choose the GL backend, then import and return ``robosuite`` (raises :class:`SimError` if missing)."""
    import_mujoco()
    _empty_private_macros()
    try:
        import robosuite
    except ImportError as exc:
        raise SimError(f"robosuite is not installed ({exc}); {_INSTALL_HINT}") from exc
    return robosuite


def import_robomimic_env_utils() -> ModuleType:
    """Return ``robomimic.utils.env_utils`` (robosuite imported first, mujoco_py stand-in installed)."""
    import_robosuite()
    install_mujoco_py_stub()
    try:
        import robomimic.utils.env_utils as env_utils
    except ImportError as exc:
        raise SimError(f"robomimic is not importable ({exc}); {_INSTALL_HINT}") from exc
    return env_utils
