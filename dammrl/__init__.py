"""dammrl: event-triggered human-robot co-adaptation for a 6-DoF rehabilitation arm."""

__version__ = "0.1.0"
