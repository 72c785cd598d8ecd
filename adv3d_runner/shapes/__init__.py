"""Vehicle library, mesh cleaning, SDF volumes and the PCA shape space."""
