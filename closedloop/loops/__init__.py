"""Loop closures: each is a residual with its Jacobians (see `base.Loop`)."""

from .base import Loop, LoopEval
from .weld import WeldLoop

__all__ = ["Loop", "LoopEval", "WeldLoop"]
