"""The history of a fleet's calibrations: identity, entries, the SQLite store, change detection, the fleet model."""
