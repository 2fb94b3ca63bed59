"""The archive index's tables, declared once (SQLAlchemy Core) for every backend.

``jobs``: one row per job folder (the folder is the record; this row is its index entry).
``targets``: one row per job and judged target with the values of its report: nominal, measured
(part frame after alignment), covariance of the measured point (upper triangle, m²), deviation,
its norm, the tolerance, the expanded uncertainty and the decision. ``part``, ``finished`` and
``serial`` are repeated from the job so that a target's trend is one index range scan of one table
(with the join to ``jobs`` for the serial, 10,000 points took twice as long on the server).

The schema is created and upgraded by the alembic migrations next to this module
(``migrations/versions``), never by ``create_all``: a migration must say the same as these tables
(``tests/test_archive_index.py`` checks it).
"""
from __future__ import annotations

import sqlalchemy as sa

metadata = sa.MetaData()

#: the columns a trend point carries besides part, target and time (in the trend index)
TREND_VALUES = ("job_id", "serial", "deviation_x", "deviation_y", "deviation_z", "deviation_norm_m", "tolerance_m",
                "uncertainty_u_m", "achieved_sigma_m", "decision", "passed")

jobs = sa.Table(
    "jobs", metadata,
    sa.Column("id", sa.String(200), primary_key=True),
    sa.Column("name", sa.String(200), nullable=False),
    sa.Column("part", sa.String(200)),  # the part's name (report.json job.part)
    sa.Column("part_number", sa.String(200)),  # report.json part.number
    sa.Column("serial", sa.String(200)),
    sa.Column("cell_id", sa.String(200)),
    sa.Column("operator", sa.String(200)),
    sa.Column("status", sa.String(20), nullable=False),
    sa.Column("verdict", sa.String(20)),
    sa.Column("started", sa.DateTime(timezone=True)),
    sa.Column("finished", sa.DateTime(timezone=True)),
    sa.Column("targets", sa.Integer),  # rows in ``targets`` written with this row (same transaction)
    sa.Column("failed", sa.Integer),
    sa.Column("sigma0_px", sa.Float),
    sa.Column("origin", sa.String(500), nullable=False),  # host:folder-root of the cell that wrote it
    sa.Column("folder", sa.String(1000), nullable=False),
    sa.Column("manifest_sha256", sa.String(64)),  # of manifest.json when indexed (None: not closed)
    sa.Column("problem", sa.Text),  # what in the folder could not be read (indexed as far as it reads)
    sa.Column("indexed_at", sa.DateTime(timezone=True), nullable=False),
    sa.Index("ix_jobs_started", "started"),
    sa.Index("ix_jobs_part_started", "part", "started"),
    sa.Index("ix_jobs_serial", "serial"),
    sa.Index("ix_jobs_part_number_started", "part_number", "started"),
)

targets = sa.Table(
    "targets", metadata,
    sa.Column("job_id", sa.String(200), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True),
    sa.Column("target_id", sa.String(100), primary_key=True),
    sa.Column("part", sa.String(200)),
    sa.Column("finished", sa.DateTime(timezone=True)),
    sa.Column("serial", sa.String(200)),
    sa.Column("kind", sa.String(20)),
    *(sa.Column(f"nominal_{a}", sa.Float, nullable=False) for a in "xyz"),
    *(sa.Column(f"measured_{a}", sa.Float) for a in "xyz"),
    *(sa.Column(f"cov_{ab}", sa.Float) for ab in ("xx", "xy", "xz", "yy", "yz", "zz")),
    *(sa.Column(f"deviation_{a}", sa.Float) for a in "xyz"),
    sa.Column("deviation_norm_m", sa.Float),
    sa.Column("tolerance_m", sa.Float),
    sa.Column("uncertainty_u_m", sa.Float),
    sa.Column("achieved_sigma_m", sa.Float),  # sqrt(trace) of the measured point's covariance (report.json)
    sa.Column("decision", sa.String(20)),  # conforming | nonconforming | inconclusive | None (not measured)
    sa.Column("passed", sa.Boolean),
    # covering: a trend reads this index alone (an index-only scan), not one table page per job
    sa.Index("ix_targets_trend", "part", "target_id", "finished", *TREND_VALUES),
)

COV_KEYS = ("xx", "xy", "xz", "yy", "yz", "zz")
COV_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
