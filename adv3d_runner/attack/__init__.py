"""Attack objectives, search algorithms (ask/tell), driver and run journal."""
