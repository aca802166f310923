"""Many robots: batch manifests, one calibration per job, and drift across a fleet.

`batch` (`closedloop batch`), `manifest` (reading and checking a manifest), `drift` (what moved between
two calibrations, in the gauge both share).
"""
