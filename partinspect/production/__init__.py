"""Many parts: batches of inspections, their results database and statistical process control.

Orchestration like :mod:`partinspect.pipeline` (which it calls once per
part); the capability and control-chart maths is in :mod:`.spc`, plain
functions on numpy arrays.
"""
