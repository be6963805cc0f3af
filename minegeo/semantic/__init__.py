"""minegeo.semantic"""
