"""minegeo.report"""
