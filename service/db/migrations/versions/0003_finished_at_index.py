"""An index on ``scenes.finished_at``: a job's first estimate of its time reads the latest
finished jobs (``SceneStore.latest_ready``), newest first, which without it would sort every
finished scene.

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_scenes_finished_at", "scenes", ["finished_at"])


def downgrade() -> None:
    op.drop_index("ix_scenes_finished_at", "scenes")
