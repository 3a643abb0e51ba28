"""Sessions with people: a sitting's run (``session``, made of the steps in
``session_steps``), the participant's display (``display``), the therapist's console
(``console``), who takes part and their consent (``participants``, ``enrolment``) and the
session protocols (``protocols/``, data).

It starts stacks through :mod:`dammrl.stack`; it imports no other room."""
