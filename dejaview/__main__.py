from dejaview.cli import main

# guarded: worker processes of ``dejaview serve`` (multiprocessing "spawn") import this module again
if __name__ == "__main__":
    main()
