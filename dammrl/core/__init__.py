"""The core library: robot, dynamics, IK, safety, task and seeds, model set, human model,
state types, metrics, errors. Numbers in, numbers out: it imports no service, no bus and
no wire schema, so every composition (in-process runner, bus services, tools) builds on it.
"""
