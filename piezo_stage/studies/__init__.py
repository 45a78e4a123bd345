"""Multi-step reproductions: the seed's identification study and the gap diagnosis's
blind suite (they use matplotlib; kept out of the core)."""
