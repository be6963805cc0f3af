"""minegeo.registration"""
