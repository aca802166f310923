"""Loop closures: each is a residual with its Jacobians (see `base.Loop`).

Every loop type has one entry in `spec.LOOP_TYPES` (type name -> its module), the one registry
the CLI parser (`spec.parse_loop`), ``closedloop loops``, the calibrator and the simulator read
(a simulator class registers under a type name of it).  Each type's module registers its factory
beside its class (`spec.register`) and loads on first use: importing this package loads `base`
alone, and ``closedloop.loops.WeldLoop`` (or any class below) imports its module when first asked
for (PEP 562), the camera loop (`CameraLoop`, type ``camera``) included, so that `import closedloop`
pays for no loop code it does not use.
"""

from importlib import import_module
from typing import TYPE_CHECKING

from closedloop.loops.base import Loop, LoopEval

if TYPE_CHECKING:  # what the lazy names are, for type checkers
    from closedloop.loops.camera.loop import CameraLoop
    from closedloop.loops.face import FaceLoop
    from closedloop.loops.hinge import HingeLoop
    from closedloop.loops.measured import MeasuredPointLoop, MeasuredPoseLoop
    from closedloop.loops.passive import PassiveChainLoop
    from closedloop.loops.plane import PlaneLoop
    from closedloop.loops.point import PointLoop
    from closedloop.loops.weld import WeldLoop

#: the loop classes this package exports, by the module that defines each (loaded on first use)
_LAZY = {
    "CameraLoop": "closedloop.loops.camera.loop",
    "FaceLoop": "closedloop.loops.face",
    "HingeLoop": "closedloop.loops.hinge",
    "MeasuredPointLoop": "closedloop.loops.measured",
    "MeasuredPoseLoop": "closedloop.loops.measured",
    "PassiveChainLoop": "closedloop.loops.passive",
    "PlaneLoop": "closedloop.loops.plane",
    "PointLoop": "closedloop.loops.point",
    "WeldLoop": "closedloop.loops.weld",
}

__all__ = [
    "Loop",
    "LoopEval",
    "CameraLoop",
    "FaceLoop",
    "HingeLoop",
    "MeasuredPointLoop",
    "MeasuredPoseLoop",
    "PassiveChainLoop",
    "PlaneLoop",
    "PointLoop",
    "WeldLoop",
]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
