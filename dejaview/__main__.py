from dejaview.cli import main

main()
