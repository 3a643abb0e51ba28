"""dammrl's library: every algorithm of the system (the arm's model, dynamics, IK, safety, the
task, the controller and its trigger, the simulation, the human agent and its intent
sources, the arm's drivers, the policy, the posterior, the metrics). No bus, no services,
no schemas: numbers in, numbers out; the services and the tools build on it."""

__version__ = "0.1.0"
