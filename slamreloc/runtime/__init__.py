"""How the process runs: compute precision, progress bars, memory given back."""
