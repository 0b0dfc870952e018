"""Benchmarks and studies (``glsldiff bench ...``, ``glsldiff demo``): error against run time,
each compared with a peer (scipy direct / pyamg, the single-resolution solver) in the same run,
written as a printed table, CSV and a PNG plot. The library never imports it.
"""
