"""eigencast host: the pipeline, one subpackage per stage (docs/architecture.md).

`host.volume` (load a volume) -> `host.render` (ray-cast views into a Cinema database) ->
`host.fit` (eigenspace model) -> `host.evaluate` (quality and cost) | `host.link` (provision
and serve a device); `host.commands` is the CLI over them.
"""

__version__ = "0.1.0"
