"""Statistics of shape collections: the log map, Karcher means, distance matrices, tangent
PCA.
"""
