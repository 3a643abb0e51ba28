"""What a lab keeps after its sessions: the catalogue of every participant, session and
trial (``catalogue``), the clinical outcomes and their reports (``outcomes``) and the BIDS
export (``bids``).

The top room under the command line: it reads the recordings (:mod:`dammrl.stack`), the
sessions' folders and logs (:mod:`dammrl.people`) and the study's statistics
(:mod:`dammrl.study`); nothing but the command line imports it."""
