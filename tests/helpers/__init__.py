"""Helpers shared by the tests, imported as ``tests.helpers.<module>`` (pytest puts the
checkout's root on ``sys.path``: ``pythonpath`` in ``pyproject.toml``).

- :mod:`.worlds`: synthetic places and noisy drives over them (descriptors, no images);
- :mod:`.road_map`: a small map of drives over one road, with positions (trace, viewer);
- :mod:`.hmm_synth`: multi-drive place-recognition scenarios for the HMM;
- :mod:`.serve`, :mod:`.fleet`: the service's and the Ray fleet's processes and maps;
- :mod:`.crash_worker`: the crash harness (also run as a script, the killed child);
- :mod:`.index_contract` and :mod:`.contracts`: contract suites each implementation's test
  class subclasses (zarr-python's ``StoreTests`` is the model).
"""
