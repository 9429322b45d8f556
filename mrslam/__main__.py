from mrslam.cli import main
from schemas.stopping import follow_parent

if __name__ == "__main__":   # not again in a process the server starts (spawn)
    follow_parent()          # started by a launcher (the demo): end with it
    main()
