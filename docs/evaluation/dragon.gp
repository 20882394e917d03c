set terminal pngcairo size 900,600 font 'DejaVu Sans,10'
set output 'dragon.png'
set title 'dragon: deviation from the uniform surface vs triangles'
set xlabel 'output triangles'
set ylabel 'Hausdorff distance (% of diagonal)'
set logscale x
set key outside right
set grid
plot for [i=0:10] 'dragon.dat' index i using 1:2 with linespoints title columnheader(1)
