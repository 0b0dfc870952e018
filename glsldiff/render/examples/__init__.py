"""Example scenes shipped with glsldiff (``glsldiff render --example NAME``); each is rendered
by tests/test_examples.py. Copy one next to your mesh and edit it to start a scene of your own."""
