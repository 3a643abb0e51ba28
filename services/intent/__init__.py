"""Intent service: the human agent. core.py is the simulated human of the paper."""
