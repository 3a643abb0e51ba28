"""Simulation service: MuJoCo steps the arm under the joint impedance law (core.py)."""
