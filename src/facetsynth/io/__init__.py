"""Files and their checks: EXR, JSON, YAML and .npy I/O, the per-point tables, output folders that never overwrite
an input, schema validation, the one input error, colour encoding, parallel frame work.
"""
