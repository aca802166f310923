"""Reading and writing at the edge of the package: joint logs (CSV) and ROS bags, camera info, the
schemas every option, manifest and config value is checked against, and files written whole.

`logs` (`read_log`, `JointLog`), `bags` (ROS 1/ROS 2 JointState recordings to logs), `camera_info`,
`robot_files` (`read_model_file`: a URDF, MJCF or D-H table read and checked once, before a model is built),
`schemas` (JSON schemas and option values: numbers, noise, bounds), `files` (`OutputSet`,
`atomic_write_text`, `check_outputs`: an output never replaces an input, a reader never sees half a file).
`marker` (`mark_running`: the line a supervising process waits for before it interrupts the work).
Nothing here knows about kinematics.
"""
