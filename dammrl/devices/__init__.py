"""The devices a person drives the arm with, and their stand-ins: the pressure pad over a
serial port (``sensor``), wearable intent over Lab Streaming Layer (``wearable``), and the
emulated devices that replace any of them and the real arm (``emulators``: the pad, EMG and
IMU streams, a patient, the Dynamixel servo chain).

It imports :mod:`dammrl.stack` for the recordings' reader only."""
