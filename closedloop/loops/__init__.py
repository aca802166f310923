"""Loop closures: each is a residual with its Jacobians (see `base.Loop`).

Every loop type has one entry in `spec.LOOP_TYPES` (type name -> its module), the table
the CLI parser (`spec.parse_loop`), ``closedloop loops`` and the simulator read; a type's
module loads on first use, the camera loop (`CameraLoop`, type ``camera``) included, so
that `import closedloop` pays for no camera code.
"""

from .base import Loop, LoopEval
from .hinge import HingeLoop
from .measured import MeasuredPointLoop, MeasuredPoseLoop
from .passive import PassiveChainLoop
from .plane import PlaneLoop
from .point import PointLoop
from .weld import WeldLoop

__all__ = ["Loop", "LoopEval", "CameraLoop", "HingeLoop", "MeasuredPointLoop", "MeasuredPoseLoop",
           "PassiveChainLoop", "PlaneLoop", "PointLoop", "WeldLoop"]


def __getattr__(name: str):
    if name == "CameraLoop":  # loaded on first use (PEP 562)
        from .camera import CameraLoop

        return CameraLoop
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
