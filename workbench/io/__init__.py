"""File input and output with geometry: volumes, label maps, fields, meshes, weight maps, JSON; atomic writes."""
