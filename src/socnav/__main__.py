"""`python -m socnav`: the `socnav` command line (same as the installed `socnav` script)."""

from socnav.cli import main

if __name__ == "__main__":
    main()
