"""The per-frame tracker: the driver (``odometry.Odometry``), the decision in phases
(``decision``, over the records of ``records``), the host actions it asks for (``effects``:
the solves, the recovery search, the making of a keyframe; ``places``: the keyframe map's
queries), the one judgement of a verified alignment (``verify``) and the back end it hands
keyframes to (``backend``)."""
