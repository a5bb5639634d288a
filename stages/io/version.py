"""The version of the built-in readers of meshes, point files, LAS/LAZ and E57 (IFC and STEP have their own)."""

# 1.1.0: bad files (counts the data does not hold, tokens that are not numbers, truncated binaries, degenerate
# facets) are errors or dropped instead of becoming data. 1.2.0: LAS/LAZ carry intensity and colour. 1.3.0: LAS/LAZ
# keep the per-point classification (for a registrar's `classes`).
VERSION = "1.3.0"
