"""What a record says: records and excitations, identification (the fast exact solver,
the swarms, the Prandtl-Ishlinskii class) and the sim-to-real gap diagnosis. Builds on
core.model; imports nothing of core.loop."""
