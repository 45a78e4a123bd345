"""What a stage is: the Duhem hysteresis law (whole and segmented), play operators for
memory, the unmodelled effects, the exact inverse, the simulated two-axis plant and the
model document. Imports nothing of the core's other two jobs."""
