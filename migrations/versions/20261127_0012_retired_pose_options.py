"""pose options the pose stage no longer has are dropped from the option documents stored
with environments, comparisons and jobs (``max_rmse_voxels``: the inlier RMSE no longer
decides ``verified``), so that a stored override does not fail every later job as an
unknown option. The downgrade leaves the documents as they are: the old code's default
stands for a dropped override.

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-27 22:00:00
"""

from collections.abc import Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: option names removed from the pose stage, as they may stand in a ``"pose"`` section
RETIRED_POSE_OPTIONS = ("max_rmse_voxels",)
TABLES = ("environments", "comparisons", "jobs")


def without_retired(doc: Any) -> Any:
    """``doc`` with every retired option removed from each ``"pose"`` object at any depth
    (a stage's options may nest the pose stage's: ``{"compare": {"pose": {...}}}``)."""
    if isinstance(doc, dict):
        return {
            key: (
                {k: without_retired(v) for k, v in value.items() if k not in RETIRED_POSE_OPTIONS}
                if key == "pose" and isinstance(value, dict)
                else without_retired(value)
            )
            for key, value in doc.items()
        }
    if isinstance(doc, list):
        return [without_retired(v) for v in doc]
    return doc


def upgrade() -> None:
    conn = op.get_bind()
    for name in TABLES:
        table = sa.table(name, sa.column("id", sa.String), sa.column("options", sa.JSON))
        for row in conn.execute(sa.select(table.c.id, table.c.options)).all():
            cleaned = without_retired(row.options)
            if cleaned != row.options:
                conn.execute(
                    table.update().where(table.c.id == row.id).values(options=cleaned)
                )


def downgrade() -> None:
    pass
