"""minegeo.slam"""
