"""The muscle-mss application on the six filters: the ``muscle-mss`` command (run, demo, study,
validate), its options and output folder, the motion run that chains the filters per time point,
the study and its report, the pictures, and the kernels' warm-up."""
