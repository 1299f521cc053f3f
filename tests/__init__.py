"""The test suite, a package so that its shared helpers have one import path from every test
file, test worker and benchmark: ``from tests.references import ...`` (the NumPy references)."""
