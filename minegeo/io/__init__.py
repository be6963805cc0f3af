"""minegeo.io"""
