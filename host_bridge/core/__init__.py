"""The host's core, below every other layer: records (options, robot and topic state, grids, the
robot model), the converter contract, decoding, columns, frame naming, counters, and the only
calls of Rerun's private API (``rerun_private``)."""
