"""Virtual-lab presets shared by the tests."""


from core.lab.generate import PRESETS

SHORT_DURATION = 6.0
"""Sequence length of the tests' sessions, s."""

SHORT_SMALL = PRESETS["small"].with_duration(SHORT_DURATION)
"""The `small` preset with 6 s sequences (train x 2, validation, test): one or two pokes
per sequence, the least that exercises a fit or a diagnosis; the suite's time depends on it."""
