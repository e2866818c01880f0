"""Drivers of whole runs: a sequence (``run``), a batch of sequences and configurations
(``batch``), a sweep (``sweep``, ``sweep_file``, ``processes``), the camera's calibration
(``calibrate``), a fit of the learnable ``Params`` (``fit``), one frame pair (``pair``) and
the measurements the benchmarks share (``measure``)."""
