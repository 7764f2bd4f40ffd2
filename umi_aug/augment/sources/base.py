"""The one seam between an input and the export: :class:`InputSource`, and the registry that picks one for a path.

The export (:func:`umi_aug.augment.exporter.export`) asks a source, in this order and never by its kind:

1. :meth:`~InputSource.reads` — the paths the source reads (the export refuses to write inside them);
2. :meth:`~InputSource.check` — every input checked before anything is computed or removed: ONE
   :class:`~umi_aug.errors.AugmentError` naming the file, key, episode or value;
3. :meth:`~InputSource.fingerprint` — the content (and settings) hash that enters the run key and the stage keys;
4. :attr:`~InputSource.dataset` and :meth:`~InputSource.n_augment` — the UMI replay buffer whose episodes are the
   originals (copied into the export), and how many of them are augmented (for the disk-space estimate);
5. :meth:`~InputSource.prepare` — run (or find cached) the source's stages and return the
   :class:`~umi_aug.augment.session_assets.SessionAssets` handle that the episode loop, the planner and the
   renderer consume: ``cfg``, ``work_dir``, ``demos`` and ``augmentable``, ``original`` (the originals' buffer),
   ``for_demo(d)`` (the handle of demo ``d``'s scene: SDF, Gaussians, render views, overlay mask),
   ``umi_episode(episode, d)`` (the UMI keys of a new episode) and ``stages`` (for the summary); a source
   whose scenes are built per demo on demand (a plain dataset) also names them, ``scene_to_build(d)`` and
   ``build_scene(key)``, so the export runs each build as a task of its own ahead of its episodes.

:func:`register_source` adds a kind (a detector and a factory); :func:`open_source` gives the source of the first
kind whose detector claims the path, or the default kind's (a UMI session) when none does.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from umi_aug.augment.config import AugmentConfig
from umi_aug.augment.session_assets import SessionAssets
from umi_aug.errors import AugmentError

__all__ = ["InputSource", "SourceFactory", "register_source", "open_source", "source_kind", "source_kinds",
           "settings_from_cli"]


class InputSource(Protocol):
    """An input of the export (see the module doc for the order the export calls it in)."""

    @property
    def dataset(self) -> Path:
        """The UMI replay buffer (``*.zarr.zip`` or zarr directory) whose episodes are the originals."""
        ...

    def reads(self) -> tuple[Path, ...]:
        """The files and folders this input reads: the export never writes into (or deletes) them."""
        ...

    def check(self, image_size: int) -> Any:
        """Check every input before any compute, for policy images of ``image_size`` pixels; returns what it read.

        Raises:
            AugmentError: the first problem, naming the file/key/episode/value.
        """
        ...

    def fingerprint(self) -> str:
        """Hash of the input's content and settings: part of the export's run key (a change starts over)."""
        ...

    def n_augment(self, n_episodes: int) -> int:
        """How many of the ``n_episodes`` original episodes are augmented."""
        ...

    def prepare(self, work: Path, cfg: AugmentConfig, *, progress: bool = True,
                prefit_obstacles: Sequence[str] = ()) -> SessionAssets:
        """Run (or skip, when cached under ``work``) the input's stages; return the episode loop's handle.

        ``prefit_obstacles``: the obstacle assets the export's first attempts draw (a source may fit them early,
        beside a long stage; others fit each asset when an episode first uses it).
        """
        ...


#: ``factory(path, settings)``: the source of ``path`` (as the caller gave it: messages name it so); ``settings``
#: are the kind's own input settings (a :class:`~umi_aug.augment.dataset_source.DatasetInput`, or those of a kind
#: registered from a package above, e.g. the square demos' ``SquareInput``) or None for its defaults.
SourceFactory = Callable[["str | os.PathLike", Any], InputSource]


@dataclass(frozen=True)
class _Kind:
    name: str
    detect: Callable[[Path], bool] | None  # None: the default kind
    factory: SourceFactory
    from_cli: Callable[[Any], Any] | None = None  # parsed `umi-aug augment` flags -> the kind's settings


_KINDS: list[_Kind] = []


def register_source(kind: str, detect: Callable[[Path], bool] | None, factory: SourceFactory,
                    from_cli: Callable[[Any], Any] | None = None) -> None:
    """Add an input kind: ``detect(path)`` claims a path (asked in registration order, cheap, never raises),
    ``factory(path, settings)`` opens it, ``from_cli(args)`` (optional) makes its settings from the parsed
    ``umi-aug augment`` flags (:func:`settings_from_cli`). ``detect=None`` makes ``kind`` the default: the source
    of any path no other kind claims (one default; its :meth:`~InputSource.check` says what the path is not).
    Registering a kind again replaces it in place.

    Raises:
        AugmentError: a second default kind.
    """
    new = _Kind(kind, detect, factory, from_cli)
    for i, k in enumerate(_KINDS):
        if k.name == kind:
            _KINDS[i] = new
            return
    if detect is None and any(k.detect is None for k in _KINDS):
        raise AugmentError(f"register_source({kind!r}): a default input kind is registered already "
                           f"({[k.name for k in _KINDS if k.detect is None][0]!r})")
    _KINDS.append(new)


def _kind_of(path: Path) -> _Kind:
    for k in _KINDS:
        if k.detect is not None and k.detect(path):
            return k
    for k in _KINDS:
        if k.detect is None:
            return k
    raise AugmentError(f"{path}: no input kind claims it (registered: {source_kinds()})")


def source_kinds() -> list[str]:
    """The registered kinds, in the order their detectors are asked (the default last)."""
    return [k.name for k in _KINDS if k.detect is not None] + [k.name for k in _KINDS if k.detect is None]


def source_kind(path: str | os.PathLike) -> str:
    """The kind of input at ``path`` (``"dataset"``, ``"session"`` or a registered one, e.g. ``"square"``); reads
    only what the detectors read, raises nothing for the built-in kinds."""
    return _kind_of(Path(path)).name


def open_source(path: str | os.PathLike, settings: Any = None) -> InputSource:
    """The :class:`InputSource` of ``path``: its kind's factory called with ``settings`` (the kind's own input
    settings, None for its defaults). Nothing is checked here (:meth:`InputSource.check` does)."""
    return _kind_of(Path(path)).factory(path, settings)


def settings_from_cli(kind: str, args: Any) -> Any:
    """The input settings of a registered ``kind`` from the parsed ``umi-aug augment`` flags ``args`` (its
    ``from_cli``; None — the kind's defaults — when it registered none)."""
    for k in _KINDS:
        if k.name == kind:
            return None if k.from_cli is None else k.from_cli(args)
    raise AugmentError(f"input kind {kind!r}: not registered (registered: {source_kinds()})")
