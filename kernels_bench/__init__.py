"""Benchmarks and studies (run as scripts); ``stability_cases`` is also imported by the tests."""
