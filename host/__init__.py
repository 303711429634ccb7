"""eigencast host: volumes, ray-casting, eigenspace fitting, evaluation, serving."""

__version__ = "0.1.0"
