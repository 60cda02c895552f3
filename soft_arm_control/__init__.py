"""Two-level controller of the soft arm (collocated P-satI-D+ inner loop, underactuated CLIK)."""
