"""Offline studies: the paper's identification study, the gap diagnosis's blind suite
and the sparse hysteresis peer (they use matplotlib or pysindy; kept out of the core)."""
