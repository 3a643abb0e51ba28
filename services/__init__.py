"""The services of the stack: one package each, a pure core and (later) a bus node."""
