"""Statistics (intervals, the bootstrap, numbers for people) and the paper's claims."""
