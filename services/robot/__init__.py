"""Stage S3, the real arm: a Dynamixel Protocol 2.0 servo chain (the emulated chain so far;
the robot service and its driver are issue 16's next steps)."""
