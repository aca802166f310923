"""The robot, task and scene files shipped with closedloop, and the catalogue that finds them.

`catalog` (`ROBOTS`, `model_file`, `nominal_urdf`, the example-robot-data locator); the files:
``utah_mit_hand.urdf`` and ``dh/`` (the thesis's hand), ``planar3.urdf``, ``door.xml`` (a MuJoCo door),
``tasks/`` (door, drawer, crank: task chains for ``passive`` loops).
"""
