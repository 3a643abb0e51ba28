"""The session catalogue: every participant, session, block and trial found again, in an
embedded database (DuckDB), built from the recordings and the sessions' trial logs.

MCAP stays the raw record. Each recording a session made carries, in its metadata, which
participant, session, protocol (name, version, SHA-256), block and trials its stack run
served (``dammrl.session`` -> ``study``); each reach in it ends with its EpisodeResult.
The catalogue reads them (each file once, checked: ``recordings``) and the sessions'
trial logs, nothing else, so it can be deleted and rebuilt identically at any time
(``dammrl session catalogue``), and every row points back into its recording: the file
and the reach's time range (log times, ns). How it is built, kept fresh and read
without harm: ``store``.

Tables (``<root>/catalogue/catalogue.duckdb``):

* ``participants``: one row per participant, their number of sessions.
* ``sessions``: participant, session, protocol, its version and SHA-256, the first and
  last message's time, the trials and successes, and its data completeness: the reaches
  its trial log holds, recorded whole, in part or missing, and reaches with no line.
* ``trials``: one row per reach of a trial (``attempt``; ``final`` marks the attempt that
  counts: a trial the therapist ran again keeps its earlier attempts), its block and
  condition, every metric of the one metrics module, the recording and time range.
* ``comfort``: the participant's ratings after each block; ``actions``: every act of the
  therapist, each as itself (pause, resume, skip, again, end-block, take, decide, give,
  stop, release), with who and why.
* ``completeness``: each session's trial log (``trials.jsonl``) reconciled with its
  recordings, line by line: recorded whole, in part, missing (and why), skipped; and
  reaches recorded with no line (``ledger``).
* ``recordings``: every file read, used or passed over, complete or cut, and what was
  wrong with it.

``trials`` is also written as Parquet, one file per session under
``<root>/catalogue/trials/participant=<id>/session=<ses>/`` (Hive partitioning), for
tools that read Parquet (pandas, R's arrow, DuckDB itself).

The modules, bottom up: ``tables`` (the columns), ``recordings`` (each file read once and
checked), ``ledger`` (the trial logs reconciled), ``store`` (building, freshness, reading
without harm), ``queries``. They import the recordings' reader (``dammrl.stack.recording``), the
session folder's log (``dammrl.people.session``) and the library; nothing imports them but the
reports, the BIDS export and the CLI.
"""

from dammrl.data.catalogue.queries import trials_of
from dammrl.data.catalogue.store import (
    Built,
    Table,
    build,
    catalogue_path,
    connect,
    ensure,
    query,
    stale,
)
from dammrl.data.catalogue.tables import (
    METRICS,
    TRIAL_COLUMNS,
    CatalogueError,
    UnreadableCatalogueError,
)

__all__ = [
    "METRICS",
    "TRIAL_COLUMNS",
    "Built",
    "CatalogueError",
    "Table",
    "UnreadableCatalogueError",
    "build",
    "catalogue_path",
    "connect",
    "ensure",
    "query",
    "stale",
    "trials_of",
]
