"""Images in: a frame's edges, gradients and distance-field pyramid (host preprocessing),
and reading those fields at sub-pixel points (device)."""
