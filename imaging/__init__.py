"""imaging package."""

__all__: list[str] = []
