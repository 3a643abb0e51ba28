"""dammrl's tools, grouped by the jobs a lab does (one sub-package, a "room", per job; see
docs/reference/architecture.md): running the arm (``stack``), sessions with people
(``people``), what a lab keeps (``data``), seeing a run (``views``), the person's devices
and their emulators (``devices``), learning the policy (``learning``), the paper's study
(``study``), and the command line over all of them (``cli``). Built on the services, the
library (:mod:`dammrl_core`) and the contract (:mod:`schemas`)."""

from dammrl_core import __version__

__all__ = ["__version__"]
