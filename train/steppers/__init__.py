"""The neural-stepper problems, one file each, registered with
:data:`adjointsim.train.problems.STEPPERS` (found by ``adjointsim data``, ``train`` and the
studies)."""
