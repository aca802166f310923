"""What a user gets on disk: the calibrated model and the report.

`urdf` (URDF and D-H writers), `mjcf` (MJCF writer), `report` (the JSON report and the sensors file),
`html` (the self-contained HTML report).
"""
