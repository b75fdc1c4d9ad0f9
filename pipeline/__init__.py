"""The pipeline: DAG declaration, runner, config, catalog I/O and CLI."""
