"""minegeo.synth"""
