"""Scene file schema and validation, generators, importers and background geometry."""
