"""The host side: the streaming odometry state (``Odometry``), running a sequence, batched
evaluation of many sequences and configurations, and the run's summary."""
