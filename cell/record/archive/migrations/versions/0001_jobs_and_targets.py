"""The archive index: jobs and their per-target measured values.

Revision ID: 0001
Revises:
Create Date: 2026-11-22
"""
import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

TZ = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "jobs",
        sa.Column("id", sa.String(200), primary_key=True),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("part", sa.String(200)),
        sa.Column("part_number", sa.String(200)),
        sa.Column("serial", sa.String(200)),
        sa.Column("cell_id", sa.String(200)),
        sa.Column("operator", sa.String(200)),
        sa.Column("status", sa.String(20), nullable=False),
        sa.Column("verdict", sa.String(20)),
        sa.Column("started", TZ),
        sa.Column("finished", TZ),
        sa.Column("targets", sa.Integer),
        sa.Column("failed", sa.Integer),
        sa.Column("sigma0_px", sa.Float),
        sa.Column("origin", sa.String(500), nullable=False),
        sa.Column("folder", sa.String(1000), nullable=False),
        sa.Column("manifest_sha256", sa.String(64)),
        sa.Column("problem", sa.Text),  # what in the folder could not be read (indexed as far as it reads)
        sa.Column("indexed_at", TZ, nullable=False),
    )
    op.create_index("ix_jobs_started", "jobs", ["started"])
    op.create_index("ix_jobs_part_started", "jobs", ["part", "started"])
    op.create_index("ix_jobs_serial", "jobs", ["serial"])
    op.create_index("ix_jobs_part_number_started", "jobs", ["part_number", "started"])
    op.create_table(
        "targets",
        sa.Column("job_id", sa.String(200), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("target_id", sa.String(100), primary_key=True),
        sa.Column("part", sa.String(200)),
        sa.Column("finished", TZ),
        sa.Column("serial", sa.String(200)),
        sa.Column("kind", sa.String(20)),
        *(sa.Column(f"nominal_{a}", sa.Float, nullable=False) for a in "xyz"),
        *(sa.Column(f"measured_{a}", sa.Float) for a in "xyz"),
        *(sa.Column(f"cov_{ab}", sa.Float) for ab in ("xx", "xy", "xz", "yy", "yz", "zz")),
        *(sa.Column(f"deviation_{a}", sa.Float) for a in "xyz"),
        sa.Column("deviation_norm_m", sa.Float),
        sa.Column("tolerance_m", sa.Float),
        sa.Column("uncertainty_u_m", sa.Float),
        sa.Column("achieved_sigma_m", sa.Float),
        sa.Column("decision", sa.String(20)),
        sa.Column("passed", sa.Boolean),
    )
    op.create_index("ix_targets_trend", "targets", ["part", "target_id", "finished", "job_id", "serial", "deviation_x",
                                                    "deviation_y", "deviation_z", "deviation_norm_m", "tolerance_m",
                                                    "uncertainty_u_m", "achieved_sigma_m", "decision", "passed"])


def downgrade() -> None:
    op.drop_table("targets")
    op.drop_table("jobs")
