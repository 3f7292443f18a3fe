"""Jobs as every layer sees them: their specifications (``specs``), checks, files and dispatch."""
