-- Run once, when the PostgreSQL volume is created: the database `mlflow` is created by the
-- image (POSTGRES_DB); Optuna gets its own, as both keep an `alembic_version` table.
CREATE DATABASE optuna;
