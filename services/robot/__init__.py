"""Stage S3, the real arm: the robot service (the sim's contract on a Dynamixel Protocol 2.0
chain), its driver, the arm's calibration and an emulated servo chain for work without
hardware."""
