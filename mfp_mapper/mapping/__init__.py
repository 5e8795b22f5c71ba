"""The mapping loop: sources -> the scan pipeline -> the Mapper, with one set of counters. The
node's live worker, the offline replay, folder replay and the fleet run it."""
