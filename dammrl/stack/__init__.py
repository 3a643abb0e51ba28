"""Running the arm: the stack of services on the bus (``launch``), the operator's stop
(``stop``), what a run recorded (``recording``: the MCAP reader every other room uses),
looking into a run and a file (``inspect``), replaying a recording onto a bus or into the
policy (``replay``), and the same services composed in one process for whole reaches
(``runner``).

The floor every other room stands on: it imports the services, the library and the
contract, and nothing else of ``dammrl``."""
