"""minegeo.survey"""
