"""The one error the twin store raises."""


class TwinStoreError(Exception):
    """A clear, user-facing twin store error naming the twin path, epoch or key."""
