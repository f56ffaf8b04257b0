"""The `lightfield` command line: a thin adapter over core, service and worker."""
