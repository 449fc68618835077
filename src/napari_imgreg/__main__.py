import sys

from napari_imgreg.cli import main

sys.exit(main())
