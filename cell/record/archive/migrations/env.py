"""Alembic environment of the archive index: run on the connection the cell hands over.

The cell calls ``alembic.command.upgrade`` itself on every open (:meth:`ArchiveIndex._ensure_schema`)
with ``config.attributes["connection"]`` set, inside its migration lock. By hand, with an ini file
whose ``[alembic]`` section says ``script_location = <this folder>``::

    alembic -c that.ini -x url=postgresql://user@host:5432/archive current    (or: upgrade head)
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import context

from cell.record.archive.tables import metadata

config = context.config
connection = config.attributes.get("connection")

if connection is None:  # run from the alembic command line: -x url=...
    url = context.get_x_argument(as_dictionary=True).get("url")
    if not url:
        raise SystemExit("give the archive's database: alembic -x url=sqlite:///... or postgresql://...")
    if url.startswith("postgres"):
        from cell.record.archive.postgres import engine_url

        url = engine_url(url)
    engine = sa.create_engine(url)
    with engine.begin() as connection:
        context.configure(connection=connection, target_metadata=metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
else:
    context.configure(connection=connection, target_metadata=metadata,
                      render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        context.run_migrations()
