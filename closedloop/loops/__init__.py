"""Loop closures: each is a residual with its Jacobians (see `base.Loop`).

Every loop type has one entry in `spec.LOOP_TYPES` (type name -> its module), the one registry
the CLI parser (`spec.parse_loop`), ``closedloop loops``, the calibrator and the simulator read
(a simulator class registers under a type name of it); a type's module loads on first use, the
camera loop (`CameraLoop`, type ``camera``) included, so that `import closedloop` pays for no
camera code.
"""

from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.hinge import HingeLoop
from closedloop.loops.measured import MeasuredPointLoop, MeasuredPoseLoop
from closedloop.loops.passive import PassiveChainLoop
from closedloop.loops.plane import PlaneLoop
from closedloop.loops.point import PointLoop
from closedloop.loops.weld import WeldLoop

__all__ = [
    "Loop",
    "LoopEval",
    "CameraLoop",
    "HingeLoop",
    "MeasuredPointLoop",
    "MeasuredPoseLoop",
    "PassiveChainLoop",
    "PlaneLoop",
    "PointLoop",
    "WeldLoop",
]


def __getattr__(name: str):
    if name == "CameraLoop":  # loaded on first use (PEP 562)
        from closedloop.loops.camera.loop import CameraLoop

        return CameraLoop
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
