"""Serving an image with several looks: the look the device shows is the look served.

A device showing look i of an image with several (`device_runtime.looks`) names it in each
VIEW_REQUEST (``look``; absent: the first). `ServedLooks.follow` is called each turn of the
stream with the look of the request just taken: when it changed, the session serves the new
look from then on -- its `HostModel` (its eigenspace and noise floor, its depth), its
ray-caster (its own render settings: transfer function, lighting), its frame sources and
refinement, and a key frame first -- and every SCORES it sends says the look it was made
for, so a device that switched again while a packet was on its way drops it. The models,
ray-casters and sources of the looks shown are kept (a switch back costs nothing).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

from host.fit.model import HostModel

__all__ = ["ServedLooks", "served_looks"]


class ServedLooks:
    """The looks of one served image, made as the device shows them.

    Parameters
    ----------
    names : tuple of str
        The image's look names.
    first : int
        The look ``model`` is (the one serving starts with).
    model : HostModel
    renderer : ViewRenderer or None
        ``model``'s ray-caster.
    load : callable
        ``load(index) -> HostModel`` of another look.
    open_renderer : callable
        ``open_renderer(model) -> ViewRenderer or None`` (None: serve it without ray-casts).
    """

    def __init__(self, names: tuple[str, ...], first: int, model: HostModel,
                 renderer: Any | None, load: Callable[[int], HostModel],
                 open_renderer: Callable[[HostModel], Any | None]) -> None:
        self.names = names
        self._models: dict[int, HostModel] = {first: model}
        self._renderers: dict[int, Any | None] = {first: renderer}
        self._sources: dict[int, dict] = {}
        self._load = load
        self._open_renderer = open_renderer
        self._refused: set[int] = set()

    def follow(self, run: Any, look: int) -> bool:
        """Serve ``look`` from now on in ``run`` (a `host.link.serving._Serving`) when it is
        not the look served: its model in the encoder (the next packet a key frame), its
        ray-caster, its frame sources and resting refinement (`_Serving._pick` on the
        session's HELLO_REPLY), the view on show refined anew; one line says so. A look the
        image lacks is said once and not served. Returns whether the look changed."""
        if look == run.look:
            return False
        if not 0 <= look < len(self.names):
            if look not in self._refused:
                self._refused.add(look)
                run.say(f"the device asks for look {look}; the image has {len(self.names)} "
                        f"({', '.join(self.names)}): serving look {self.names[run.look]}")
            return False
        model = self._models.get(look)
        if model is None:
            model = self._models[look] = self._load(look)
        if look not in self._renderers:
            self._renderers[look] = self._open_renderer(model)
        from host.link.serving import _Shown

        self._sources.setdefault(run.look, run.sources)  # the look left keeps its sources
        run.encoder.model = model
        run.encoder.reset()
        run.renderer = self._renderers[look]
        run.sources = self._sources.setdefault(look, {})
        run.look = look
        shown = run.current
        run.current = _Shown(view=shown.view, sequence=shown.sequence,
                             requested_at=shown.requested_at)
        run.failed_view = None
        if run.hello is not None:
            run._pick(run.hello)
        run.stats.look_switches += 1
        how = ("ray-cast with its render settings" if run.renderer is not None
               else "no ray-cast")
        run.say(f"the device shows look {self.names[look]}: serving it ({how})")
        return True

    def close(self) -> None:
        """Drop every look's frame sources."""
        for sources in self._sources.values():
            sources.clear()


def served_looks(model: HostModel, model_path: str | os.PathLike, key: bytes | None,
                 renderer: Any | None, open_renderer: Callable[[HostModel], Any | None]
                 ) -> ServedLooks | None:
    """The `ServedLooks` of ``model`` (loaded from ``model_path``, verified with ``key``;
    its ray-caster ``renderer``); None: its image has one look."""
    if not model.looks:
        return None
    names = tuple(model.looks)
    return ServedLooks(names, names.index(model.look), model, renderer, lambda index: (
        HostModel.load(model_path, key=key, look=names[index])), open_renderer)
