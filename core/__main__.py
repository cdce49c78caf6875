"""``python -m lrslam`` = the ``lrslam`` command."""

from lrslam.cli import main

if __name__ == "__main__":
    main()
