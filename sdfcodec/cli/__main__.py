"""``python -m sdfcodec.cli``: the same as the ``sdfcodec`` command."""

from . import main

main()
