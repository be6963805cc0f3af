"""minegeo.geometry"""
