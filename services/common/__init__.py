"""Code the API, the worker and the graph store share: problem details and error mapping, the
dataset catalog, upload checks and the submit path. Imports nothing from ``services.api``."""
