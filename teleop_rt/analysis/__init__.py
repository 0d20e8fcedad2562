"""Analysis: transparency metrics (eq 18) and the displayed impedance (eq 19-32)."""
