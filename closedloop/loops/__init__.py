"""Loop closures: each is a residual with its Jacobians (see `base.Loop`).

Importing this package registers every loop type for the CLI (`spec.parse_loop`).
"""

from .base import Loop, LoopEval
from .measured import MeasuredPointLoop, MeasuredPoseLoop
from .plane import PlaneLoop
from .point import PointLoop
from .weld import WeldLoop

__all__ = ["Loop", "LoopEval", "MeasuredPointLoop", "MeasuredPoseLoop", "PlaneLoop", "PointLoop", "WeldLoop"]
