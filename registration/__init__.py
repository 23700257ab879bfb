"""registration package."""

__all__: list[str] = []
