"""Tracking (the front end): the distance residual and its Jacobian, robust weights, the
coarse-to-fine alignment of a keyframe's edges to a frame, edge selection and the keyframe
decision."""
