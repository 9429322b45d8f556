from mrslam.cli import main

if __name__ == "__main__":   # not again in a process the server starts (spawn)
    main()
