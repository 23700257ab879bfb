from heartreg.cli import run

run()
