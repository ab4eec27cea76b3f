"""Command-line entry points (bake, benchmarks, extension build)."""
