"""Detection, prediction, planning and realism metrics."""
