from td3_jax.cli import main

main()
