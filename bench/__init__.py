"""Benchmarks behind `pag bench <name>`; each module has main(argv) and writes under data/bench/."""
