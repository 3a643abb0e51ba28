"""Message models, codec and key expressions of the bus (the bus issue)."""
