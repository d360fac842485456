"""DRAN: the decentralized solver (Algorithm 1), its consensus, messages and initialisation."""
