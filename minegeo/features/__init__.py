"""minegeo.features"""
