from partinspect.cli import console

console()
