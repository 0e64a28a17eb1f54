"""Mission programs that ship with baton: the paper's grid, and a corridor survey."""
