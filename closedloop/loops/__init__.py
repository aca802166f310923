"""Loop closures: each is a residual with its Jacobians (see `base.Loop`).

Importing this package registers every loop type for the CLI (`spec.parse_loop`).
"""

from .base import Loop, LoopEval
from .camera import CameraLoop
from .hinge import HingeLoop
from .measured import MeasuredPointLoop, MeasuredPoseLoop
from .passive import PassiveChainLoop
from .plane import PlaneLoop
from .point import PointLoop
from .weld import WeldLoop

__all__ = ["Loop", "LoopEval", "CameraLoop", "HingeLoop", "MeasuredPointLoop", "MeasuredPoseLoop",
           "PassiveChainLoop", "PlaneLoop", "PointLoop", "WeldLoop"]
