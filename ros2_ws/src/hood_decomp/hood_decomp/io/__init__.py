"""File I/O: model and mesh files, the ensemble store, saved bases, bags. Never pickle."""
