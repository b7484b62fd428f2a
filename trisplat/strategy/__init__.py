"""Soft-to-hard strategy: the topology ops (the only code that edits vertex/face tables), pruning, densification, opacity floor."""
