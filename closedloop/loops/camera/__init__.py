"""Camera loops: a marker on the robot seen by one or more cameras (pinhole and lens models, stereo).

`loop` (the loop and its Jacobians), `model` (projection, distortion, DLT), `start` (the starting values
from the pixels), `stereo` (triangulation), `spec` (the ``camera:`` spec of the loop registry; importing
this package registers it).
"""

from closedloop.loops.camera import spec  # noqa: F401  (registers the 'camera' loop type)
