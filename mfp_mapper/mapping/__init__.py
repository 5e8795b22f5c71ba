"""The mapping loop: sources -> the scan pipeline -> the Mapper, with one set of counters. The
node's live worker, the offline replay of any recording (``sources.recording``), localization
against a map and the fleet run it."""
