"""The numeric core: pose-graph factors, problems, Schur-complement LM, sparse Cholesky,
chordal initialisation, the SE-Sync objective and the centralized solver (paper Sec. 4).
"""
