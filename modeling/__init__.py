"""modeling package."""

__all__: list[str] = []
