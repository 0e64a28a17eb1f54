"""The station network's fleet side: which stations a mission needs (admission) and
the registry that remembers stations and admitted missions."""
