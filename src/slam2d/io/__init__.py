"""Reading and writing files: trajectory export (TUM), graph formats, dataset loaders."""
