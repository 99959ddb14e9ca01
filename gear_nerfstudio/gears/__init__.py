"""Gear-assignment updates (Sec 4.3): schedule, loss maps and prompts, upshift targets and steps, the updater."""
