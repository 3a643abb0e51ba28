"""What services share: bus session and settings, logging, health (the bus issue)."""
