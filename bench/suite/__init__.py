"""Building blocks of `lightfield bench`: measurement, evaluation, simulated suites, stability."""
