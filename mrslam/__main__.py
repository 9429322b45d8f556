from mrslam.cli import main

main()
