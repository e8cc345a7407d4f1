from cell.cli import main

main()
