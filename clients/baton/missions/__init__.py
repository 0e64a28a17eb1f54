"""Mission programs that ship with baton (the paper's grid mission)."""
