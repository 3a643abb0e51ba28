"""Seeing a run: the live 3D view for Foxglove (``viewer``, behind the WebSocket gate
``wsgate``; its JSON schemas in ``foxglove_schemas/``), videos of reaches (``video``) and
the figures of a recording (``plots``).

It reads recordings and reaches from :mod:`dammrl.stack`; the study draws with ``plots``."""
