"""Learning the policy: the Dual-Agent DQN's environment and training (``rl``) and the
per-person refinement behind its gate (``adapt``).

It runs reaches with :mod:`dammrl.stack`'s in-process runner; the study uses it."""
