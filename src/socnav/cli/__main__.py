"""`python -m socnav.cli`: the `socnav` command."""

from socnav.cli import main

if __name__ == "__main__":
    main()
