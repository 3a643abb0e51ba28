"""Controller service: micro-steps, progression (event trigger / fixed timer), IK,
joint reference, inverse-dynamics feedforward and safety holds (core.py)."""
