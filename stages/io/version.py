"""The version of the built-in readers of meshes, point files, LAS/LAZ and E57 (IFC and STEP have their own)."""

# 1.1.0: bad files (counts the data does not hold, tokens that are not numbers, truncated binaries, degenerate
# facets) are errors or dropped instead of becoming data. 1.2.0: LAS/LAZ carry intensity and colour.
VERSION = "1.2.0"
