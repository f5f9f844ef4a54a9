"""Input/output: dataset loaders producing :class:`slam2d.log.Log` (``io.datasets``) and graph file formats."""
