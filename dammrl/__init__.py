"""dammrl's tools and compositions: the command line, the in-process runner, RL training,
the studies, the launcher, recordings, viewers. Built on the services, the library
(:mod:`dammrl_core`) and the contract (:mod:`schemas`)."""

from dammrl_core import __version__

__all__ = ["__version__"]
