"""Applications: what runs the node set for a purpose (``demo``, ``replay`` of a bag,
the control ``experiments`` and the relay experiment for tuning) and the offline
``studies`` (the paper's identification study, the gap diagnosis's blind suite, the
sparse peer)."""
