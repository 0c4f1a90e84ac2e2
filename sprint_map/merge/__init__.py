"""After a drive: which decisions become edges (the rule, verification) and the commit."""

__all__: list[str] = []
