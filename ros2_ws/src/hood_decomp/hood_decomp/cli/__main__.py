from hood_decomp.cli import entry

entry()
