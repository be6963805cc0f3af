"""minegeo.mast"""
