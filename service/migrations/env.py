"""Alembic environment: runs the migrations on the connection `upgrade_database` hands over.

Standalone use (`alembic` CLI) is not needed: `sfmnerf db upgrade` and the service's start-up upgrade.
"""

from alembic import context

from service.store.tables import Base

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=Base.metadata)
with context.begin_transaction():
    context.run_migrations()
