# sdfcodec's pytest plugin (--regen-golden, the regen_golden fixture) loads by itself where sdfcodec is installed
# with its pytest11 entry point; this line loads it otherwise, and is a no-op when it is already loaded.
pytest_plugins = ["sdfcodec.testing.pytest_plugin"]
